"""The operator dashboard and the guest kiosk in a real browser (Debian's chromium, headless, WebGL
through SwiftShader) against a real `flockcal serve` process reading the simulated performer on a pty:
the skeleton renders, the bones table matches the simulator's body, an injected slip appears on the
residual plot and as an alert, an unplugged tracker and a restarted server are shown and recovered
from by the pages themselves, and the kiosk reaches "done" on the kiosk routine and takes the next guest.

Screenshots go to $FLOCKCAL_ARTIFACTS (default: artifacts/ in the repository, git-ignored).
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from server_helpers import ServerProcess, free_port, wait_connected
from service_process import wait_for
from flockcal.simulator.performer import Performer
from browser_helpers import NEEDS_CHROMIUM

pytestmark = [
    pytest.mark.browser,
    NEEDS_CHROMIUM,
]

ADMIN, KIOSK, READ = "admin-secret-1", "kiosk-secret-1", "read-secret-1"
SLIP_SENSOR = "l_forearm"
SLIP_AFTER_S = 14.0
# docs/dashboard.md "Measured": bones end within 0.9–3.1 mm of the simulator's between ball joints and
# 10–23 mm where a bone ends at a hinge (measured while the fit's centre there was the min-norm point along
# the hinge axis; the limb rule of docs/design.md §3c now places it, and the bound is kept). Margins for a loaded 2-core machine, where the page may show a fit a
# few hundred frames older than the newest: 1.4 mm and 7 mm.
BONE_TOLERANCE_M = 0.023 + 0.007
BALL_BONE_TOLERANCE_M = 0.0031 + 0.0014
LIMIT = {"hinge": BONE_TOLERANCE_M, "ball": BALL_BONE_TOLERANCE_M}
# The kiosk shows the service's progress (its target: serve's default 5 mm); the kiosk routine exercises
# each limb once a loop.
KIOSK_QUERY = f"token={KIOSK}&reset_s=3"
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def performer():
    # As conftest's, with rigid sensors: the drawn bones are held to the simulator's true bones (1 cm
    # between ball joints), and soft tissue, on by default, moves the fitted joint centres by about that.
    return Performer("human", "exercise", seed=1, rate_hz=144.0, period=8.0, sta_mm=0)


def artifacts() -> Path:
    path = Path(os.environ.get("FLOCKCAL_ARTIFACTS") or ROOT / "artifacts")
    path.mkdir(parents=True, exist_ok=True)
    return path


def record(key: str, value) -> None:
    """Keep a measured figure with the screenshots (docs/dashboard.md "Measured" quotes them)."""
    path = artifacts() / "dashboard-figures.json"
    figures = json.loads(path.read_text()) if path.exists() else {}
    figures[key] = value
    path.write_text(json.dumps(figures, indent=1))


def admin() -> dict:
    return {"Authorization": f"Bearer {ADMIN}"}


@pytest.fixture(scope="module")
def server(tracker, performer, tmp_path_factory):
    data = tmp_path_factory.mktemp("dashboard")
    args = ["--device", tracker.device, "--birds", "16", "--data-dir", str(data), "--fast-init",
            "--names", ",".join(performer.names), "--scale", "72", "--baud", "921600", "--token", ADMIN, "--kiosk-token", KIOSK, "--read-token", READ]
    proc = ServerProcess(args, free_port(), log_path=data / "serve.log").start(token=ADMIN)
    wait_connected(proc.url, token=ADMIN)
    yield proc
    proc.stop()


def open_page(browser, url: str, width: int = 1440, height: int = 1000):
    page = browser.new_page(viewport={"width": width, "height": height})
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.goto(url)
    return page


@pytest.fixture(scope="module")
def dashboard(browser, server):
    """The dashboard with a session started from its own form, once the fit has every joint."""
    page = open_page(browser, f"{server.url}/?token={ADMIN}")
    page.wait_for_selector("#tracker[data-state=connected]", timeout=20000)
    page.fill("#performer", "Ann")
    page.click("#start")
    page.wait_for_selector("#session-state[data-state=live]", timeout=10000)
    # Every sensor but the root with a fitted joint (none still riding rigidly on a neighbour).
    page.wait_for_function("document.querySelectorAll('#coverage .cov:not([data-state=rigid])').length >= 15",
                           timeout=40000)
    yield page
    page.close()


def wait_until(predicate, timeout: float, what: str, interval: float = 0.25):
    return wait_for(predicate, timeout, what, every=interval)


def transitions_done(page, selector: str) -> None:
    """Wait until the CSS transitions of `selector` have run (for a picture of where they end)."""
    page.wait_for_function("s => document.querySelector(s).getAnimations().every(a => a.playState !== 'running')",
                           arg=selector, timeout=10000)


def canvas_pixels(page, selector: str, colours: list[str], tolerance: int = 40) -> dict:
    """Counts of pixels in a canvas: total, differing from its background (top-left pixel), near each colour."""
    return page.evaluate(
        """([sel, colours, tol]) => {
            const src = document.querySelector(sel);
            const c = document.createElement('canvas');
            c.width = src.width; c.height = src.height;
            const ctx = c.getContext('2d');
            ctx.drawImage(src, 0, 0);
            const d = ctx.getImageData(0, 0, c.width, c.height).data;
            const bg = [d[0], d[1], d[2]];
            const want = colours.map((h) => [1, 3, 5].map((k) => parseInt(h.slice(k, k + 2), 16)));
            const near = (i, rgb) => Math.abs(d[i] - rgb[0]) + Math.abs(d[i + 1] - rgb[1]) + Math.abs(d[i + 2] - rgb[2]) < tol;
            const out = { total: d.length / 4, changed: 0, colours: colours.map(() => 0) };
            for (let i = 0; i < d.length; i += 4) {
                if (!near(i, bg)) out.changed += 1;
                want.forEach((rgb, k) => { if (near(i, rgb)) out.colours[k] += 1; });
            }
            return out;
        }""",
        [selector, colours, tolerance],
    )


def bone_rows(page) -> list[dict]:
    return page.eval_on_selector_all(
        "#bones tbody tr[data-body]",
        "rows => rows.map(r => ({body: r.dataset.body, from: r.dataset.from || null, to: r.dataset.to, "
        "length: Number(r.dataset.lengthM)}))",
    )


def true_joint_points(truth: dict) -> dict:
    """{(body, frozenset(joint bodies)): the joint centre in that body's sensor frame} from the simulator."""
    out = {}
    for j in truth["joints"]:
        pair = frozenset((j["child"], j["parent"]))
        out[(j["child"], pair)] = np.asarray(j["c"], dtype=float)
        out[(j["parent"], pair)] = np.asarray(j["l"], dtype=float)
    return out


def test_dashboard_draws_the_skeleton_and_bones_match_the_simulator(dashboard, performer, server):
    page = dashboard
    assert page.get_attribute("#view", "data-renderer") == "webgl"
    page.wait_for_function("Number(document.querySelector('#view').dataset.frames) > 10", timeout=10000)
    # The 3D view draws spheres (green when calibrated, amber otherwise), bones and sensor boxes. Bones end
    # only at determined joints, so they appear as the joints are pinned: give them the first loops.
    def drawn():
        px = canvas_pixels(page, "#view canvas", ["#3fb950", "#ffc857", "#3fa9f5", "#e4572e"], tolerance=60)
        ok = (px["changed"] > 0.01 * px["total"] and sum(px["colours"][:2]) > 50 and px["colours"][2] > 200
              and px["colours"][3] > 20)
        return px if ok else None

    wait_until(drawn, 20, "joints, bones and sensors drawn in the 3D view")

    truth = performer.truth()
    points = true_joint_points(truth)
    hinges = {frozenset((n, truth["parent"][n])) for n, t in zip(performer.model.names, performer.model.joint_type)
              if t == "hinge"}

    def shown_bones():
        sid = httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["id"]
        parent = httpx.get(f"{server.url}/api/sessions/{sid}/result", headers=admin()).json()["parent"]
        rows = bone_rows(page)
        # The page's rows and /result come from two reads of a live fit: when the tree changed in between
        # (a joint the page names is the root of the other, or not in it), read both again.
        if any(c and c not in parent for r in rows for c in (r["from"], r["to"])):
            return None
        # The fit may root the tree elsewhere than the simulator: name each joint by its two bodies.
        for r in rows:
            r["joints"] = [frozenset((c, parent[c])) for c in (r["from"], r["to"]) if c]
        # Every bone the simulated body has is shown (rigid sensors: every joint gets determined).
        return rows if len(rows) >= len(truth["bones"]) and all(len(r["joints"]) == 2 for r in rows) else None

    def errors():
        rows = shown_bones()
        if rows is None:
            return None
        out = []
        for r in rows:
            a, b = (points.get((r["body"], j)) for j in r["joints"])
            if a is None or b is None:  # a joint the simulated body does not have (a wrong tree)
                out.append(("no such joint", r, np.inf))
                continue
            # A bone ending at a hinge depends on the point a rule chooses along the hinge axis.
            kind = "hinge" if any(j in hinges for j in r["joints"]) else "ball"
            out.append((kind, r, abs(r["length"] - float(np.linalg.norm(a - b)))))
        return out

    def converged():
        errs = errors()
        return errs if errs and all(e < LIMIT.get(k, 0.0) for k, _, e in errs) else None

    # The live fit improves as the performer moves: every bone must come within tolerance.
    try:
        errs = wait_until(converged, 30, "every bone within tolerance of the simulator's")
    except AssertionError:
        bad = [(k, r["body"], sorted(map(sorted, r["joints"])), round(e, 4)) for k, r, e in errors() or []
               if e >= LIMIT.get(k, 0.0)]
        raise AssertionError(f"bones still off after 30 s: {bad}") from None
    worst = {k: max([e for kk, _, e in errs if kk == k], default=0.0) for k in ("ball", "hinge")}
    record("bones_worst_error_m", worst)
    record("bones_shown", {"rows": len(errs), "truth": len(truth["bones"])})
    page.screenshot(path=str(artifacts() / "dashboard-bones.png"), full_page=True)
    assert not page.errors


def test_injected_slip_shows_on_the_residual_plot_and_as_an_alert(dashboard, performer, server):
    page = dashboard
    page.wait_for_function("Number(document.querySelector('#residuals').dataset.samples) > 20", timeout=10000)
    before = page.eval_on_selector_all(".alert.slip", "els => els.filter(e => /left forearm/.test(e.textContent)).length")
    sid = httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["id"]

    def service_slip():
        events = httpx.get(f"{server.url}/api/sessions/{sid}/events", headers=admin()).json()["events"]
        return [e for e in events if e["type"] == "slip" and SLIP_SENSOR in [e.get("sensor"), *e.get("candidates", [])]]

    # Slip once the tree has settled and the detector has a full loop of motion as its baseline (a
    # slip while the topology still changes is missed: the monitor restarts with every new tree).
    wait_until(lambda: httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["time_s"] >= SLIP_AFTER_S,
               30, f"{SLIP_AFTER_S} s of session")
    performer.inject_slip(SLIP_SENSOR, 0.03)
    wait_until(service_slip, 10, "the service reporting the slip")
    # Whatever the service reports reaches the page within a few seconds.
    page.wait_for_function(
        "[...document.querySelectorAll('.alert.slip')].filter(e => /left forearm/.test(e.textContent)).length > %d"
        % before, timeout=5000)
    slips = int(page.get_attribute("#residuals", "data-slips"))
    assert slips >= 1
    # The marker is drawn on the plot: dashed red lines in the uPlot canvas.
    wait_until(lambda: canvas_pixels(page, "#residuals canvas", ["#f85149"], tolerance=60)["colours"][0] > 30, 10,
               "the slip's marker drawn on the plot")
    text = page.text_content("#alerts")
    assert re.search(r"Sensor slipped: [^—]*left forearm", text), text
    # A little more plot after the slip, for the picture: two seconds more of the session.
    slipped_at = httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["time_s"]
    wait_until(lambda: httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["time_s"] >= slipped_at + 2,
               30, "two seconds more of the session")
    page.screenshot(path=str(artifacts() / "dashboard.png"), full_page=True)
    assert not page.errors


def test_a_page_opened_after_the_slip_still_marks_it_on_the_residual_plot(browser, server):
    """Tried as issue #29 did: a dashboard opened well after a slip (the websocket replays only the last
    5 s of residuals). Its 60 s plot used to start at the page load, without the slip's marker; it now
    starts from the session's own residuals and events, so the marker is on it."""
    sid = httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["id"]
    events = httpx.get(f"{server.url}/api/sessions/{sid}/events", headers=admin()).json()["events"]
    slips = [e for e in events if e["type"] == "slip" and SLIP_SENSOR in [e.get("sensor"), *e.get("candidates", [])]]
    assert slips, "no slip in the session: the test before injects it"
    slip = slips[0]
    # Opened 10 s after the slip: past the websocket's replay, well inside the plot's 60 s.
    wait_until(lambda: httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["time_s"]
               >= slip["time_s"] + 10, 60, "10 s after the slip")
    page = open_page(browser, f"{server.url}/?token={ADMIN}")
    try:
        page.wait_for_function(
            "(t) => { const d = document.querySelector('#residuals').dataset;"
            " return Number(d.slips) >= 1 && d.first !== '' && Number(d.first) <= t; }",
            arg=slip["time_s"], timeout=15000)
        px = canvas_pixels(page, "#residuals canvas", ["#f85149"], tolerance=60)
        assert px["colours"][0] > 30, px  # the dashed red marker is drawn
        assert not page.errors
    finally:
        page.close()


def test_pages_show_an_unplugged_tracker_and_recover(dashboard, browser, server, tracker):
    page = dashboard
    kiosk = open_page(browser, f"{server.url}/kiosk?token={READ}", 1600, 900)  # read-only: follows the live session
    try:
        kiosk.wait_for_selector("#kiosk-state[data-tracker=connected]", timeout=15000)
        # A read-only kiosk cannot start a guest session: it shows the one the operator started.
        # (live, or already done by its own targets: either way it names her and started nothing).
        kiosk.wait_for_function("['live', 'done'].includes(document.querySelector('#kiosk-state').dataset.state)",
                                timeout=15000)
        assert "Ann" in kiosk.text_content("#kiosk-state")
        assert httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["performer"] == "Ann"
        tracker.disconnect()
        try:
            page.wait_for_selector("#tracker[data-state=disconnected]", timeout=15000)
            assert page.is_visible("#banner") and "Tracker disconnected" in page.text_content("#banner")
            kiosk.wait_for_selector("#kiosk-state[data-tracker=disconnected]", timeout=15000)
            assert "tracker is disconnected" in kiosk.text_content("#banner")
            page.screenshot(path=str(artifacts() / "dashboard-unplugged.png"))
        finally:
            tracker.reconnect()
        page.wait_for_selector("#tracker[data-state=connected]", timeout=30000)
        kiosk.wait_for_selector("#kiosk-state[data-tracker=connected]", timeout=30000)
        assert page.is_hidden("#banner") and kiosk.is_hidden("#banner")
        assert not page.errors and not kiosk.errors
    finally:
        kiosk.close()


def test_pages_reconnect_by_themselves_after_a_server_restart(dashboard, browser, server):
    page = dashboard
    kiosk = open_page(browser, f"{server.url}/kiosk?token={READ}", 1600, 900)
    try:
        kiosk.wait_for_selector("#kiosk-state[data-link=open]", timeout=15000)
        server.stop()
        page.wait_for_selector("#link[data-state=closed]", timeout=15000)
        assert page.is_visible("#link-banner")
        kiosk.wait_for_function("document.querySelector('#kiosk-state').dataset.link !== 'open'", timeout=15000)
        assert "Reconnecting" in kiosk.text_content("#banner")
        server.start(token=ADMIN)
        # No reload: each page reconnects and streams again (frames count moves on).
        page.wait_for_selector("#link[data-state=open]", timeout=30000)
        page.wait_for_selector("#tracker[data-state=connected]", timeout=30000)
        # The restarted service counts frames from zero, so "moves on" means changes, not exceeds.
        first = int(page.text_content("#fig-frames").replace(",", ""))
        page.wait_for_function(f"Number(document.querySelector('#fig-frames').textContent.replace(/,/g, '')) !== {first}",
                               timeout=15000)
        kiosk.wait_for_selector("#kiosk-state[data-link=open]", timeout=30000)
        assert page.is_hidden("#link-banner")
        # The restart ended the operator's session; the read-only kiosk waits for a host, starting nothing.
        kiosk.wait_for_selector("#kiosk-state[data-state=waiting]", timeout=15000)
        assert httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"] is None
        assert not page.errors and not kiosk.errors
    finally:
        kiosk.close()


def test_session_controls_start_stop_and_download_the_skeleton(dashboard, server):
    page = dashboard
    # The fixture's session may still be live (when this test runs without the restart test before it):
    # the Start button only comes back once it has stopped.
    live = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
    if live:
        httpx.post(f"{server.url}/api/sessions/{live}/stop", headers=admin(), timeout=30)
    page.wait_for_selector("#link[data-state=open]", timeout=30000)
    page.wait_for_selector("#start:not([disabled])", timeout=15000)
    page.fill("#performer", "Bo")
    page.click("#start")
    page.wait_for_selector("#session-state[data-state=live]", timeout=10000)
    sid = httpx.get(f"{server.url}/api/status", headers=admin()).json()["session"]["id"]
    page.wait_for_function("document.querySelectorAll('#bones tbody tr[data-body]').length >= 4", timeout=20000)
    page.click("#stop")
    page.wait_for_selector("#session-state[data-state=stopped]", timeout=30000)
    assert httpx.get(f"{server.url}/api/sessions/{sid}", headers=admin()).json()["state"] == "stopped"
    with page.expect_download(timeout=15000) as info:
        page.click("#dl-skeleton")
    downloaded = json.loads(Path(info.value.path()).read_text())
    served = httpx.get(f"{server.url}/api/sessions/{sid}/skeleton", headers=admin()).json()
    downloaded.pop("created_utc"), served.pop("created_utc")  # stamped when each file is made
    assert downloaded == served
    # The skeleton file is the one `flockcal serve --skeleton` loads for the performer's next take.
    from flockcal.exports.skeleton import parse_skeleton
    assert parse_skeleton(Path(info.value.path()).read_text()).hierarchy
    assert info.value.suggested_filename == f"Bo-{sid}-skeleton.json"
    with page.expect_download(timeout=15000) as info:
        page.click("#dl-bvh")
    assert Path(info.value.path()).read_text().startswith("HIERARCHY")
    assert info.value.suggested_filename == f"Bo-{sid}.bvh"
    with page.expect_download(timeout=15000) as info:
        page.click("#dl-gltf")
    assert Path(info.value.path()).read_bytes()[:4] == b"glTF"  # the binary container's magic (glTF 2.0 §4.4)
    assert info.value.suggested_filename == f"Bo-{sid}.glb"
    with page.expect_download(timeout=15000) as info:
        page.click("#dl-trc")
    assert Path(info.value.path()).read_text().startswith("PathFileType\t4\t(X/Y/Z)")
    assert info.value.suggested_filename == f"Bo-{sid}.trc"
    assert not page.errors


def test_kiosk_reaches_done_on_the_kiosk_routine_and_starts_the_next_guest(browser, server, performer):
    live = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
    if live:
        httpx.post(f"{server.url}/api/sessions/{live}/stop", headers=admin(), timeout=30)
    performer.clear_faults()
    performer.set_routine("kiosk")
    page = open_page(browser, f"{server.url}/kiosk?{KIOSK_QUERY}", 1600, 900)
    try:
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        started = time.monotonic()
        guest = httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"]
        assert guest is not None
        page.wait_for_selector("#kiosk-state[data-state=done]", timeout=75000)
        record("kiosk_seconds_to_done", round(time.monotonic() - started, 1))
        transitions_done(page, "#ring-fill")  # the ring where its transition ends, for the picture
        page.screenshot(path=str(artifacts() / "kiosk.png"))
        # "Done" is the service's: the guest's session is stored done, with every joint calibrated, and its
        # stored calibration has every joint (tests/test_kiosk_browser.py checks the ring step by step).
        session = wait_until(lambda: (s := httpx.get(f"{server.url}/api/sessions/{guest}", headers=admin()).json())
                             ["state"] == "stopped" and s, 15, "the kiosk stopping the guest's session")
        assert session["performer"].startswith("guest") and session["done"] is True
        stored = httpx.get(f"{server.url}/api/sessions/{guest}/progress", headers=admin()).json()
        assert stored["joints_done"] == stored["joints_needed"] == len(performer.names) - 1
        result = httpx.get(f"{server.url}/api/sessions/{guest}/result", headers=admin()).json()
        assert len(result["joints"]) == len(performer.names) - 1
        # After reset_s the kiosk starts a fresh session for the next guest by itself.
        page.wait_for_selector("#kiosk-state[data-state=live]", timeout=15000)
        nxt = wait_until(lambda: httpx.get(f"{server.url}/api/sessions", headers=admin()).json()["live"], 10,
                         "a new guest session")
        assert nxt != guest
        assert page.eval_on_selector("body", "b => !b.classList.contains('done')")
        assert not page.errors
    finally:
        page.close()
