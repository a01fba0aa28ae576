"""A season at the kiosk, in headless chromium against a real `flockcal serve` on a fake tracker (pty):
the dashboard's season panel shows /api/stats; a tracker unplugged mid-guest comes back and the kiosk hands
the guest on (max_s) and starts the next one by itself; a kiosk page left open through a ten-minute
outage of the service keeps trying every few seconds and recovers on its own when the service is back.

The ten minutes run on the page's own clock (Playwright's fake timers, fast-forwarded a minute per refused
attempt), not the wall clock: what could break over a long outage is the page's reconnect schedule (a
back-off that grows without a cap, a retry that gives up), and that lives in the page's timers. The
hour-long soak (benchmarks/bench_soak.py) runs the rest in real time.
"""

from __future__ import annotations

import time

import httpx
import pytest

from server_helpers import ServerProcess, free_port, wait_connected
from service_process import wait_for
from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker
from browser_helpers import NEEDS_CHROMIUM

pytestmark = [
    pytest.mark.browser,
    NEEDS_CHROMIUM,
]

ADMIN, KIOSK = "admin-secret-19", "kiosk-secret-19"
RATE = 144.0
OUTAGE_MS = 10 * 60 * 1000  # issue #19: a kiosk page left open through a 10-minute outage
STEP_MS = 60 * 1000  # the page's clock jumps a minute after each refused attempt
# common.js waits at most 4 s between attempts (its back-off cap); 0.5 s of margin for the page's timers.
RETRY_CAP_MS = 4000 + 500


@pytest.fixture(scope="module")
def tracker():
    performer = Performer("human", "exercise", seed=19, rate_hz=RATE, period=8.0)
    pty = PtyTracker(performer, birds=16, baud=921600, rate_hz=RATE).start()
    yield pty
    pty.stop()


@pytest.fixture(scope="module")
def server(tracker, tmp_path_factory):
    data = tmp_path_factory.mktemp("season")
    args = ["--device", tracker.device, "--birds", "16", "--data-dir", str(data), "--fast-init",
            "--names", ",".join(tracker.flock.source.names), "--scale", "72", "--baud", "921600",
            "--token", ADMIN, "--kiosk-token", KIOSK, "--keep-disk", "5"]
    proc = ServerProcess(args, free_port(), log_path=data / "serve.log").start(token=ADMIN)
    wait_connected(proc.url, token=ADMIN)
    yield proc
    proc.stop()


def admin() -> dict:
    return {"Authorization": f"Bearer {ADMIN}"}


def live_id(url: str):
    return httpx.get(f"{url}/api/sessions", headers=admin()).json()["live"]


def wait_until(fn, timeout: float, what: str):
    return wait_for(fn, timeout, what, every=0.2)


def new_page(browser, url: str, fake_clock: bool = False):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.errors, page.sockets = [], []
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.on("websocket", lambda ws: page.sockets.append(ws.url))
    # Count the page's own connection attempts as it makes them (chromium reports a throttled one late).
    page.add_init_script("""(() => { const Native = window.WebSocket; window.__attempts = 0;
        window.WebSocket = class extends Native { constructor(...a) { super(...a); window.__attempts += 1; } }; })()""")
    if fake_clock:
        page.clock.install()
    page.goto(url)
    return page


def stop_live(url: str) -> None:
    try:
        sid = live_id(url)
    except httpx.ConnectError:  # the service is down (a failed outage test): nothing live to stop
        return
    if sid:
        httpx.post(f"{url}/api/sessions/{sid}/stop", headers=admin(), timeout=30)


def test_the_dashboards_season_panel_shows_the_services_stats(browser, server):
    sid = httpx.post(f"{server.url}/api/sessions", headers=admin(), json={"performer": "guest one"}).json()["id"]
    wait_until(lambda: httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()["frames"] >= RATE, 30,
               "frames in the session")
    httpx.post(f"{server.url}/api/sessions/{sid}/stop", headers=admin(), timeout=30)
    # What was tried: the kiosk's token pinning a session (admin only), the stats with no token at all.
    r = httpx.post(f"{server.url}/api/sessions/{sid}/pin", headers={"Authorization": f"Bearer {KIOSK}"})
    assert r.status_code == 403 and not httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()["pinned"]
    assert httpx.get(f"{server.url}/api/stats").status_code == 401
    page = new_page(browser, f"{server.url}/?token={ADMIN}")
    try:
        page.wait_for_selector("#season-panel[data-loaded]", timeout=15000)
        stats = httpx.get(f"{server.url}/api/stats?days=7", headers=admin()).json()
        rows = page.eval_on_selector_all("#season-days tr", "rs => rs.map(r => [...r.cells].map(c => c.textContent))")
        assert len(rows) == 8  # seven days and the total
        assert rows[0][0] == stats["days"][0]["day"] and rows[0][1] == str(stats["days"][0]["sessions"]) != "0"
        assert rows[-1][1] == str(stats["total"]["sessions"])
        disk = page.text_content("#season-disk")
        assert "of a 5.00 GB budget" in disk and "disk free" in disk
        assert not page.errors
    finally:
        page.close()


def test_unplugged_tracker_comes_back_and_the_kiosk_takes_the_next_guest_by_itself(browser, server, tracker):
    stop_live(server.url)
    # max_s=8: a guest who has not finished after 8 s is handed on (the kiosk's give-up for a guest who
    # walks away), so the test sees the next guest's session start without waiting for a calibration.
    page = new_page(browser, f"{server.url}/kiosk?token={KIOSK}&max_s=8&reset_s=2")
    try:
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=20000)
        first = wait_until(lambda: live_id(server.url), 10, "kiosk session")
        tracker.disconnect()
        try:
            page.wait_for_selector("#kiosk-state[data-tracker=disconnected]", timeout=15000)
            assert "tracker is disconnected" in page.text_content("#banner")
            # Unplugged until the service has tried the port again and found it gone.
            tries = httpx.get(f"{server.url}/api/status", headers=admin()).json()["reconnects"]
            wait_until(lambda: httpx.get(f"{server.url}/api/status", headers=admin()).json()["reconnects"] > tries,
                       30, "a try of the unplugged port")
        finally:
            tracker.reconnect()
        page.wait_for_selector("#kiosk-state[data-tracker=connected]", timeout=30000)
        # Nobody touches anything: the kiosk ends the first guest's session and starts the next one.
        second = wait_until(lambda: (s := live_id(server.url)) and s != first and s, 40, "next guest's session")
        row = wait_until(lambda: (r := httpx.get(f"{server.url}/api/sessions/{second}", headers=admin()).json())
                         ["frames"] >= 300 and r, 30, "frames in the next guest's session")
        assert row["performer"].startswith("guest ")
        done = httpx.get(f"{server.url}/api/sessions/{first}", headers=admin()).json()
        assert done["state"] == "stopped" and done["has_result"]
        assert page.is_hidden("#banner") and not page.errors
    finally:
        page.close()
        stop_live(server.url)


def test_a_kiosk_page_left_open_through_a_ten_minute_outage_keeps_trying_and_recovers(browser, server):
    stop_live(server.url)
    page = new_page(browser, f"{server.url}/kiosk?token={KIOSK}", fake_clock=True)
    try:
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=20000)
        before = live_id(server.url)
        server.stop()
        page.wait_for_function("document.querySelector('#kiosk-state').dataset.link !== 'open'", timeout=15000)
        def refused() -> None:
            # The refused connection closes in real time (chromium itself spaces out failing websocket
            # connections by up to ~5 s); only then does the page schedule its next try. Read through
            # the DOM: the page's own timers are the fake ones.
            wait_for(lambda: page.get_attribute("#kiosk-state", "data-link") == "closed", 15,
                     "the page's connection attempt ended", every=0.02)

        attempts = lambda: page.evaluate("window.__attempts")  # noqa: E731
        tried = attempts()
        for _ in range(OUTAGE_MS // STEP_MS):
            refused()
            page.clock.fast_forward(STEP_MS)
        refused()
        assert attempts() - tried >= OUTAGE_MS // STEP_MS  # it kept trying, minute after minute
        # Ten minutes down, the next try is still at most the back-off cap away, not minutes.
        n = attempts()
        page.clock.fast_forward(RETRY_CAP_MS)
        assert attempts() == n + 1, f"no new attempt {RETRY_CAP_MS} ms after ten minutes of outage"
        assert "Reconnecting" in page.text_content("#banner")
        server.start(token=ADMIN)
        # No reload and no person: the page reconnects, sees the restarted service has no live session
        # (the restart stopped it) and starts the next guest's session by itself.
        page.wait_for_selector("#kiosk-state[data-link=open]", timeout=30000)
        after = wait_until(lambda: (s := live_id(server.url)) and s != before and s, 30, "a new guest session")
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        assert page.is_hidden("#banner") and not page.errors
        assert httpx.get(f"{server.url}/api/sessions/{before}", headers=admin()).json()["state"] == "stopped"
        assert after
    finally:
        page.close()
        stop_live(server.url)
