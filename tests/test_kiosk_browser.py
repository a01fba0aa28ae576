"""The kiosk's ring is the service's progress, step by step (issue 21): a real `flockcal serve` reads a
simulated guest on a pty whose kiosk routine starts with the kiosk's own session; headless chromium shows
the kiosk page (and the operator dashboard beside it). At every sampled moment the ring shows the percent
of the very fit message the page last drew (captured off the page's own websocket), which REST serves too
for that fit; "100 %" only ever appears when every sensor's joint in that fit is determined; the ring never
goes back on a clean take and never shows every chip ticked below 100 %; the dashboard's "joints calibrated"
and its labels say the same. The guest wears skin-mounted sensors (the simulator's default soft tissue) and
the kiosk starts its sessions under the kiosk profile (issue #30); a page that goes away ends its session
after its lease; a guest who stands still gets a patient prompt.
"""

from __future__ import annotations

import json
import math
import os
import time

import httpx
import pytest

from server_helpers import GuestSource, ServerProcess, free_port, wait_connected
from service_process import wait_for
from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker
from browser_helpers import NEEDS_CHROMIUM

pytestmark = [
    pytest.mark.browser,
    NEEDS_CHROMIUM,
]

ADMIN, KIOSK, READ = "admin-secret-21", "kiosk-secret-21", "read-secret-21"
RATE = 144.0
RING_CIRCUMFERENCE = 2 * math.pi * 86  # the ring's circle in kiosk.html has r = 86
# docs/service.md "Time to calibrate": kiosk guests with soft tissue are done within 35 s of their
# session (p90 target); the session's own clock gives it 5 s of margin. The wall-clock deadline only stops
# a hung test: a loaded machine delivers the same session seconds later.
DONE_SESSION_S = 35.0 + 5.0
DONE_WITHIN_S = 120.0


@pytest.fixture(scope="module")
def guest():
    # The simulator's default soft tissue: what skin-mounted sensors do, and what the kiosk profile is for.
    performer = Performer("human", "kiosk", seed=21, rate_hz=RATE, height=1.66)
    tracker = PtyTracker(performer, birds=16, baud=921600, rate_hz=RATE)
    stream = GuestSource(performer, tracker.flock.time)
    tracker.flock.source = stream
    tracker.start()
    yield performer, tracker, stream
    tracker.stop()


@pytest.fixture(scope="module")
def server(guest, tmp_path_factory):
    performer, tracker, _ = guest
    data = tmp_path_factory.mktemp("kiosk")
    args = ["--device", tracker.device, "--birds", "16", "--data-dir", str(data), "--fast-init",
            "--names", ",".join(performer.names), "--scale", "72", "--baud", "921600", "--token", ADMIN,
            "--kiosk-token", KIOSK, "--read-token", READ]
    proc = ServerProcess(args, free_port(), log_path=data / "serve.log").start(token=ADMIN)
    wait_connected(proc.url, token=ADMIN)
    yield proc
    proc.stop()


def admin() -> dict:
    return {"Authorization": f"Bearer {ADMIN}"}


def open_capturing(browser, url: str, width: int, height: int):
    """A page whose websocket `fit` messages are kept by fit_seq, as the page received them."""
    page = browser.new_page(viewport={"width": width, "height": height})
    page.errors, page.fits = [], {}

    def on_frame(payload):
        if isinstance(payload, str) and payload.startswith('{"type": "fit"'):
            msg = json.loads(payload)
            page.fits[msg["fit_seq"]] = msg

    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.on("websocket", lambda ws: ws.on("framereceived", on_frame))
    page.goto(url)
    return page


RING_JS = """() => {
    const el = document.querySelector('#percent');
    return {text: el.textContent, seq: el.dataset.fitSeq, offset: document.querySelector('#ring-fill').style.strokeDashoffset,
            state: document.querySelector('#kiosk-state').dataset.state,
            chips: document.querySelectorAll('#chips .chip').length,
            rule: document.querySelector('#rule').textContent,
            ticked: document.querySelectorAll('#chips .chip.done').length};
}"""

DASHBOARD_JS = """() => ({joints: document.querySelector('#s-joints').textContent,
    seq: document.querySelector('#s-joints').dataset.fitSeq,
    rows: [...document.querySelectorAll('#coverage .cov')].map(r => ({joint: r.dataset.joint, done: r.dataset.done,
                                                                      label: r.querySelector('.cov-name').textContent}))})"""


def rest_twin(page, rest: dict) -> dict | None:
    """The websocket fit message of the fit a REST reply describes, if the page was sent that one."""
    if rest.get("fit_seq") is None:
        return None
    for _ in range(8):
        if rest["fit_seq"] in page.fits:
            return page.fits[rest["fit_seq"]]
        page.wait_for_timeout(25)
    return None


def message_for(page, seq: str) -> dict:
    """The fit message the page drew last (its frame event can trail the page's drawing by a moment)."""
    for _ in range(40):
        if int(seq) in page.fits:
            return page.fits[int(seq)]
        page.wait_for_timeout(25)
    raise AssertionError(f"the page shows fit {seq}, which never came over its websocket")


def test_the_ring_is_the_services_progress_at_every_step_and_never_100_before_every_joint_is_determined(
        browser, server, guest):
    performer, tracker, stream = guest
    kiosk = open_capturing(browser, f"{server.url}/kiosk?token={KIOSK}&reset_s=30", 1600, 900)
    dashboard = open_capturing(browser, f"{server.url}/?token={READ}", 1440, 1000)
    try:
        # The guest starts the routine when the kiosk's session starts.
        sid = wait_for(lambda: httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"], 20,
                       "the kiosk starts a session", every=0.02)
        stream.begin()
        started = time.monotonic()
        shown, seen = [], {"rest": 0, "dash": 0, "labels": False}

        def look() -> bool:
            """One look at the ring, the REST progress and the dashboard; True once the ring says done."""
            ring = kiosk.evaluate(RING_JS)
            rest = httpx.get(f"{server.url}/api/sessions/{sid}/progress", headers=admin()).json()
            if ring["seq"]:
                msg = message_for(kiosk, ring["seq"])
                # The ring shows the service's percent of that very fit…
                assert ring["text"] == f"{msg['percent']}%", (ring, msg["progress"])
                assert msg["percent"] == math.floor(round(msg["progress"] * 100, 6))
                assert float(ring["offset"]) == pytest.approx(RING_CIRCUMFERENCE * (1 - msg["progress"]), abs=0.5)
                assert ring["ticked"] == msg["joints_done"] and ring["chips"] == msg["joints_needed"] == 15
                assert msg.get("profile") == "kiosk" and ring["rule"] == msg["rule"], ring
                # Never every chip ticked below 100 %: 15 ticks and 99 % told a guest nothing was left.
                assert ring["ticked"] < ring["chips"] or msg["done"], (ring, msg["percent"])
                # …"100 %" only when done, and done only when every sensor's joint in it is determined.
                if ring["text"] == "100%" or msg["done"]:
                    assert msg["done"] and ring["text"] == "100%"
                    result = msg["result"]
                    determined = {j["child"] for j in result["joints"] if j["determined"]}
                    assert set(result["sensors"]) - {result["root"]} <= determined, msg["missing"]
                else:
                    assert msg["missing"], "not done, yet nothing is missing"
                shown.append(msg["percent"])
            # REST serves the same figures as the websocket for the same fit.
            same = rest_twin(kiosk, rest)
            if same is not None:
                seen["rest"] += 1
                assert (rest["progress"], rest["percent"], rest["done"], rest["missing"], rest["joint_progress"]) == (
                    same["progress"], same["percent"], same["done"], same["missing"], same["joint_progress"])
            if len(shown) % 5 == 1 and shown:
                dash = dashboard.evaluate(DASHBOARD_JS)
                if dash["seq"] and dash["seq"] != "undefined":
                    dmsg = message_for(dashboard, dash["seq"])
                    assert dash["joints"] == f"{dmsg['joints_done']} / {dmsg['joints_needed']}"
                    assert {r["joint"] for r in dash["rows"] if r["done"] == "true"} == {
                        j["joint"] for j in dmsg["joint_progress"] if j["done"]}
                    seen["dash"] += 1
                    if not seen["labels"]:
                        # The page's own joint names (bones table, topology) are the service's labels.
                        pairs = [[j["joint"], j["parent"]] for j in dmsg["joint_progress"]]
                        js = dashboard.evaluate(
                            "async (pairs) => { const m = await import('/static/common.js');"
                            " return pairs.map(([c, p]) => m.jointLabel(c, p)); }", pairs)
                        assert js == [j["label"] for j in dmsg["joint_progress"]]
                        seen["labels"] = True
            return ring["state"] == "done"

        wait_for(look, DONE_WITHIN_S, lambda: f"the ring done (ring {shown[-1:]})", every=0.15)
        took = time.monotonic() - started
        # The ring where its transition ends, for the picture.
        kiosk.wait_for_function("document.querySelector('#ring-fill').getAnimations().every(a => a.playState !== 'running')",
                                timeout=10000)
        kiosk.screenshot(path=str(_artifacts() / "kiosk-progress.png"))
        assert shown[-1] == 100 and len(set(shown)) >= 5, shown  # the ring went through the figures
        assert all(b >= a for a, b in zip(shown, shown[1:])), f"the ring went back on a clean take: {shown}"
        assert seen["rest"] >= 3 and seen["dash"] >= 3 and seen["labels"], seen
        # What the kiosk showed is what the service keeps: the guest's session is stored done.
        stored = _wait_stopped(server, sid)
        assert stored["done"] is True and stored["missing"] == [] and stored["joints_done"] == 15
        assert stored["done_at_s"] <= DONE_SESSION_S, stored["done_at_s"]
        print(f"kiosk done after {took:.1f} s of wall time; {len(shown)} ring samples, {seen['rest']} REST matches")
        assert not kiosk.errors and not dashboard.errors
    finally:
        kiosk.close()
        dashboard.close()


def _wait_stopped(server, sid: str) -> dict:
    # A guard, not the promise (which is only that the kiosk stops it): a stop on a 2-core machine at a
    # load of 8 once took over 15 s.
    def stopped():
        doc = httpx.get(f"{server.url}/api/sessions/{sid}/progress", headers=admin()).json()
        return doc if not doc["live"] else None

    return wait_for(stopped, 45, "the kiosk stops its guest's session after done", every=0.2)


def _artifacts():
    from pathlib import Path

    path = Path(os.environ.get("FLOCKCAL_ARTIFACTS") or Path(__file__).resolve().parents[1] / "artifacts")
    path.mkdir(parents=True, exist_ok=True)
    return path


def test_a_read_only_kiosk_showing_a_hosts_session_done_goes_back_and_says_why_when_a_sensor_slips(
        browser, server, guest):
    performer, tracker, stream = guest
    r = httpx.post(f"{server.url}/api/sessions", json={"performer": "Host guest", "profile": "kiosk"}, headers=admin())
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    stream.begin()
    kiosk = open_capturing(browser, f"{server.url}/kiosk?token={READ}", 1600, 900)
    try:
        kiosk.wait_for_selector("#kiosk-state[data-state=done]", timeout=DONE_WITHIN_S * 1000)
        assert kiosk.text_content("#percent") == "100%"
        # Tried: the forearm sensor slides 3 cm on the skin after the guest was calibrated.
        performer.inject_slip("l_forearm", 0.03)
        # How soon the slip is found is judged on the session's own clock (tests/test_server_slip.py); here,
        # once the service has found it (a loaded machine's pipeline may run behind), the page follows it.
        wait_for(lambda: not httpx.get(f"{server.url}/api/sessions/{sid}/progress", headers=admin()).json()["done"],
                 60, "the service undoes the guest's done", every=0.2)
        kiosk.wait_for_selector("#kiosk-state[data-state=live]", timeout=10000)
        kiosk.wait_for_function("/sensor moved/.test(document.querySelector('#instruction').textContent)",
                                timeout=5000)
        assert "left forearm" in kiosk.text_content("#instruction")
        assert kiosk.text_content("#percent") != "100%"
        doc = httpx.get(f"{server.url}/api/sessions/{sid}/progress", headers=admin()).json()
        assert not doc["done"] and any((m.get("undone") or {}).get("reason") == "slip" for m in doc["missing"])
        assert not kiosk.errors
    finally:
        kiosk.close()
        performer.clear_faults()
        httpx.post(f"{server.url}/api/sessions/{sid}/stop", headers=admin(), timeout=30)


def test_a_guest_who_never_finishes_is_handed_on_after_max_s(browser, server, guest):
    # docs/dashboard.md: `max_s` (default 300 s) ends the session of a guest who walks away before done
    # and starts afresh; before that, a guest who stopped moving gets a patient prompt once the ring has not
    # risen for 8 s of session time (docs/service.md, Progress). Tried: a guest who stands still (the idle
    # routine: no joint ever turns enough) in front of a kiosk opened with max_s=14.
    performer, tracker, stream = guest
    live = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
    if live:
        httpx.post(f"{server.url}/api/sessions/{live}/stop", headers=admin(), timeout=30)
    still = Performer("human", "idle", seed=21, rate_hz=RATE, height=1.66, sta_mm=0)
    stream.begin(still)
    page = open_capturing(browser, f"{server.url}/kiosk?token={KIOSK}&max_s=14&reset_s=3", 1600, 900)
    try:
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        first = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
        assert first is not None
        started = time.monotonic()
        # The kiosk checks on each status message (about one a second): handed on within max_s + 2 s,
        # plus 20 s for a loaded machine's session stop and start (a stop once took over 15 s at load 8).
        prompts = []

        def handed_on():
            """The next guest's session once there is one; meanwhile, the patient prompt noted when it shows."""
            nxt = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
            if nxt and nxt != first:
                return nxt
            shown = page.evaluate("() => { const el = document.querySelector('#instruction');"
                                  " return {why: el.dataset.why, text: el.textContent}; }")
            if shown["why"] == "stalled" and not prompts:
                prompts.append(shown["text"])
                doc = httpx.get(f"{server.url}/api/sessions/{first}/progress", headers=admin()).json()
                assert doc["stalled_s"] >= 8 and doc["prompt"], doc
            return None

        wait_for(handed_on, 14 + 2 + 20, "the kiosk hands on to the next guest's session", every=0.2)
        prompt = prompts[0] if prompts else None
        waited = time.monotonic() - started
        assert waited > 14 - 1, f"handed on after {waited:.1f} s, before max_s"
        assert prompt and prompt.startswith("Take your time"), prompt
        gone = httpx.get(f"{server.url}/api/sessions/{first}", headers=admin()).json()
        assert gone["state"] == "stopped" and gone["done"] is False  # stored, and honestly not done
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        assert not page.errors
    finally:
        page.close()
        stream.begin(performer)


def test_a_guest_session_ends_after_its_lease_once_the_kiosk_page_goes_away(browser, server, guest):
    # Issue #30: a kiosk page closed just after it started the next guest left that session live, and
    # POST /api/sessions answered 409 until someone stopped it by hand. Tried: the page (lease_s=3) is
    # closed while its guest's session is live; the session must end for its lease, and the next session must
    # start.
    performer, tracker, stream = guest
    live = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
    if live:
        httpx.post(f"{server.url}/api/sessions/{live}/stop", headers=admin(), timeout=30)
    stream.begin(performer)
    page = open_capturing(browser, f"{server.url}/kiosk?token={KIOSK}&lease_s=3", 1600, 900)
    try:
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        sid = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
        row = httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()
        assert row["lease_s"] == 3 and row["profile"] == "kiosk", row
        # While the page is open it renews: the session outlives several leases.
        page.wait_for_timeout(7000)
        assert httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"] == sid
    finally:
        page.close()
    # Stopped, with the reason stored on its row (the note is written just after the stop). How long after
    # its lease ran out is the lease watcher's promise, held on a clock the test moves in test_server_lease.py;
    # here 60 s only stops a hung test.
    wait_for(lambda: (row := httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json())["state"] == "stopped"
             and "lease" in (row.get("note") or ""), 60, "the session stopped for its lease", every=0.1)
    r = httpx.post(f"{server.url}/api/sessions", json={"performer": "Next guest"}, headers=admin())
    assert r.status_code == 201, r.text
    httpx.post(f"{server.url}/api/sessions/{r.json()['id']}/stop", headers=admin(), timeout=30)


def _no_live_session(url: str) -> None:
    live = httpx.get(f"{url}/api/sessions", headers=admin()).json()["live"]
    if live:
        httpx.post(f"{url}/api/sessions/{live}/stop", headers=admin(), timeout=30)


def test_a_kiosk_opened_during_an_operators_session_waits_on_a_clear_screen_and_starts_when_it_ends(
        browser, server, guest):
    # Tried: an operator records "Ann" (a stage session) when the kiosk page opens with its kiosk token. The
    # page showed Ann to the guest as "Let's get you calibrated 53%" after a 409 in its console. It must say
    # the stage is in use, show no one's body or progress, send no request that fails, and start the guest's
    # own session once the operator stops.
    performer, tracker, stream = guest
    _no_live_session(server.url)
    stream.begin(performer)
    r = httpx.post(f"{server.url}/api/sessions", json={"performer": "Ann"}, headers=admin())
    assert r.status_code == 201, r.text
    ann = r.json()["id"]
    page = browser.new_page(viewport={"width": 1600, "height": 900})
    console, failed = [], []
    page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: console.append(str(e)))
    page.on("response", lambda resp: failed.append(f"{resp.status} {resp.url}") if resp.status >= 400 else None)
    try:
        page.goto(f"{server.url}/kiosk?token={KIOSK}")
        page.wait_for_selector("#kiosk-state[data-state=busy]", timeout=15000)
        page.wait_for_timeout(2000)  # fit and pose messages of Ann's session keep coming meanwhile
        shown = page.evaluate("""() => ({state: document.querySelector('#kiosk-state').dataset.state,
            words: document.querySelector('#kiosk-state').textContent + ' ' + document.querySelector('#instruction').textContent,
            body: document.body.innerText, percent: document.querySelector('#percent').textContent,
            seq: document.querySelector('#percent').dataset.fitSeq, chips: document.querySelectorAll('#chips .chip').length,
            avatar: getComputedStyle(document.querySelector('#avatar')).visibility})""")
        assert shown["state"] == "busy" and "in use" in shown["words"], shown
        assert "Ann" not in shown["body"] and shown["percent"] == "0%" and not shown["seq"] and not shown["chips"], shown
        assert shown["avatar"] == "hidden", shown
        assert httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"] == ann
        # The operator stops: the stage is the guests' again, and the kiosk starts its guest.
        assert httpx.post(f"{server.url}/api/sessions/{ann}/stop", headers=admin(), timeout=30).status_code == 200
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=20000)
        sid = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
        row = httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()
        assert sid != ann and row["performer"].startswith("guest ") and row["profile"] == "kiosk", row
        assert page.evaluate("getComputedStyle(document.querySelector('#avatar')).visibility") == "visible"
        assert not console and not failed, (console, failed)
    finally:
        page.close()
        _no_live_session(server.url)


def test_after_stop_the_dashboard_says_the_session_stopped_not_what_to_move_next(browser, server, guest):
    # Tried: an operator's session with "Move next" hints on the dashboard (joints still to calibrate), then
    # Stop. The dashboard went on saying "Keep moving the left ankle"; it must say the session stopped and how
    # far it got, and no fit of it sent before the stop may bring the hints back.
    performer, tracker, stream = guest
    _no_live_session(server.url)
    stream.begin(performer)
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(f"{server.url}/?token={ADMIN}")
        page.wait_for_selector("#start:not([disabled])", timeout=15000)
        page.fill("#performer", "Bea")
        page.click("#start")
        page.wait_for_selector("#next-moves .hint", timeout=30000)
        sid = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
        page.click("#stop")
        page.wait_for_selector("#next-moves[data-state=stopped]", timeout=30000)
        page.wait_for_timeout(1500)
        todo = page.text_content("#next-moves")
        assert f"Session {sid} stopped" in todo and "joints calibrated" in todo, todo
        assert "Keep moving" not in todo and not page.query_selector_all("#next-moves .hint"), todo
        row = httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()
        assert row["state"] == "stopped"
        assert not errors
    finally:
        page.close()
        _no_live_session(server.url)
