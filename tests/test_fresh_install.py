"""The README's first command on a fresh machine: a new venv,
`python3 -m venv .venv && . .venv/bin/activate && pip install . && flockcal serve`.

The repository is installed with plain `pip install <repo>` (no extras) into a new virtualenv without
system site packages, so nothing the test extra brings (websockets, httpx, playwright) can hide a
missing runtime dependency. That venv's `flockcal serve` runs on a free loopback port with a temporary
data directory; from the test environment we check that /ws/live streams fit and pose, that /docs and
/redoc name no external host and their assets load, and that the dashboard and kiosk load their scripts
(the vendored three.js and its GLTFLoader among them, which draw the session's rig) in chromium without
errors (screenshots in $FLOCKCAL_ARTIFACTS). pip's cache is used, so this costs seconds once the wheels are
cached; CI reaches PyPI for the first download.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import time
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urljoin, urlsplit

import httpx
import pytest
import websockets

from server_helpers import free_port, wait_connected, wait_ready
from browser_helpers import CHROMIUM, launch

ROOT = Path(__file__).resolve().parents[1]
LOOPBACK = ("127.0.0.1", "localhost")
# pip resolves and installs numpy, scipy, matplotlib, fastapi, … : about 20 s from a warm cache on the
# 2-core build machine, minutes on a first download.
INSTALL_TIMEOUT_S = 900

pytestmark = pytest.mark.timeout(INSTALL_TIMEOUT_S + 300)


def artifacts() -> Path:
    path = Path(os.environ.get("FLOCKCAL_ARTIFACTS") or ROOT / "artifacts")
    path.mkdir(parents=True, exist_ok=True)
    return path


class _Links(HTMLParser):
    """Every src= and href= of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.urls += [v for k, v in attrs if k in ("src", "href") and v]


def page_links(html: str) -> list[str]:
    parser = _Links()
    parser.feed(html)
    return parser.urls


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory) -> Path:
    venv = tmp_path_factory.mktemp("fresh") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(ROOT)],
                         capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    assert pip.returncode == 0, f"pip install {ROOT} failed:\n{pip.stdout[-3000:]}\n{pip.stderr[-3000:]}"
    return venv


@pytest.fixture(scope="module")
def fresh_serve(fresh_venv, tmp_path_factory):
    """The fresh venv's `flockcal serve` on the built-in simulator, as the README's first command runs it."""
    data = tmp_path_factory.mktemp("fresh-data")
    port = free_port()
    log = data / "serve.log"
    env = {"PATH": f"{fresh_venv / 'bin'}:/usr/bin:/bin", "HOME": str(data), "XDG_DATA_HOME": str(data),
           "LANG": "C.UTF-8", "PYTHONUNBUFFERED": "1"}
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(fresh_venv / "bin" / "flockcal"), "serve", "--http-port", str(port),
                                 "--data-dir", str(data / "flockcal")], stdout=out, stderr=subprocess.STDOUT,
                                env=env, cwd=data)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_ready(url, 60, proc=proc)
        wait_connected(url, 30)
        # A session, as an operator would start one, so fits stream and the pages have one to show.
        r = httpx.post(url + "/api/sessions", json={"performer": "Fresh"}, timeout=10)
        assert r.status_code == 201, r.text
        proc.url, proc.log = url, log
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


def test_fresh_install_has_a_websocket_library_and_no_test_extras(fresh_venv):
    # What a user gets from `pip install .`: the runtime dependencies only.
    code = ("import importlib.util as u; print(*(n for n in ('websockets','fastapi_offline','tqdm','pythonosc',"
            "'pytest','httpx','playwright') if u.find_spec(n)))")
    found = subprocess.run([str(fresh_venv / "bin" / "python"), "-c", code], capture_output=True, text=True,
                           check=True).stdout.split()
    assert {"websockets", "fastapi_offline", "tqdm", "pythonosc"} <= set(found)  # pythonosc: `serve --osc`
    assert not {"pytest", "playwright"} & set(found)  # the install really had no test extra


def test_live_websocket_streams_fit_and_pose(fresh_serve):
    async def listen() -> dict[str, int]:
        seen: dict[str, int] = {}
        async with websockets.connect(fresh_serve.url.replace("http://", "ws://") + "/ws/live") as ws:
            hello = json.loads(await asyncio.wait_for(ws.recv(), 10))
            assert hello["type"] == "hello"
            await ws.send(json.dumps({"type": "subscribe", "rate_hz": 10, "content": ["fit", "pose"]}))
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not (seen.get("fit", 0) >= 2 and seen.get("pose", 0) >= 5):
                msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                seen[msg["type"]] = seen.get(msg["type"], 0) + 1
                if msg["type"] == "fit":
                    assert msg["result"]["sensors"], "a fit message carries the §5 result"
                if msg["type"] == "pose":
                    assert len(msg["pose"]["sensors"]) == 16
        return seen

    seen = asyncio.run(listen())
    assert seen.get("fit", 0) >= 2 and seen.get("pose", 0) >= 5, seen
    assert "No supported WebSocket library" not in fresh_serve.log.read_text()


def test_the_wheel_serves_the_vendored_vrm_loader(fresh_serve):
    """three-vrm (what reads the rig as a VRM humanoid, tests/test_vrm_browser.py) ships in the wheel with
    its licence, importing the vendored three.js beside it."""
    js = httpx.get(fresh_serve.url + "/static/vendor/three-vrm/three-vrm.module.min.js", timeout=30)
    assert js.status_code == 200 and 'from"../three/three.module.js"' in js.text and 'from"three"' not in js.text
    licence = httpx.get(fresh_serve.url + "/static/vendor/three-vrm/LICENSE", timeout=30)
    assert licence.status_code == 200 and "MIT License" in licence.text


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_api_docs_name_no_external_host_and_their_assets_load(fresh_serve, page):
    html = httpx.get(fresh_serve.url + page, timeout=10)
    assert html.status_code == 200
    links = page_links(html.text)
    assert links, f"{page} links no script or stylesheet"
    external = [u for u in links if urlsplit(urljoin(fresh_serve.url + page, u)).hostname not in LOOPBACK]
    assert not external, f"{page} loads from outside the service: {external}"
    assert not re.search(r"https?://(?!127\.0\.0\.1|localhost)", html.text), f"{page} names an external URL"
    for u in links:
        asset = httpx.get(urljoin(fresh_serve.url + page, u), timeout=10)
        assert asset.status_code == 200 and len(asset.content) > 500, (u, asset.status_code)


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"needs Debian's chromium at {CHROMIUM} (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()


def open_offline(browser, url: str, width: int = 1440, height: int = 1000):
    """A page whose every request off the loopback is refused (an offline kiosk) and noted."""
    page = browser.new_page(viewport={"width": width, "height": height})
    page.problems = []
    page.scripts = []

    def route(r):
        if urlsplit(r.request.url).hostname in LOOPBACK:
            r.continue_()
        else:
            page.problems.append(f"external request {r.request.url}")
            r.abort()

    page.route("**/*", route)
    page.on("pageerror", lambda e: page.problems.append(f"page error {e}"))
    page.on("console", lambda m: m.type == "error" and page.problems.append(f"console error {m.text}"))
    page.on("requestfailed", lambda r: page.problems.append(f"failed {r.url} ({r.failure})"))
    page.on("response", lambda r: (r.request.resource_type == "script" and page.scripts.append((r.url, r.status)))
            or (r.status >= 400 and page.problems.append(f"HTTP {r.status} {r.url}")))
    page.goto(url)
    return page


@pytest.mark.browser
def test_dashboard_and_kiosk_load_their_scripts_and_go_live_in_chromium(fresh_serve, browser):
    page = open_offline(browser, fresh_serve.url + "/")
    page.wait_for_selector("#tracker[data-state=connected]", timeout=20000)
    page.wait_for_function("document.querySelectorAll('#coverage .cov').length >= 5", timeout=40000)
    # The skeleton is the session's glTF rig, parsed by the vendored GLTFLoader: its files are in the wheel.
    page.wait_for_selector("#view[data-rig=shown]", timeout=40000)
    page.wait_for_timeout(1500)
    page.screenshot(path=str(artifacts() / "fresh-dashboard.png"))
    assert page.scripts and all(status == 200 for _, status in page.scripts), page.scripts
    assert any(u.endswith("dashboard.js") for u, _ in page.scripts)
    assert "connecting" not in page.inner_text("header").lower()
    # The Alerts box wraps a long word (the sim:// URL of the tracker's "connected" event, shown when the
    # page was open while the tracker connected) instead of scrolling sideways. The alert is built as
    # dashboard.js builds one, so the page's own stylesheet lays it out.
    overflow = page.evaluate("""(() => {
        const box = document.querySelector('#alerts'), div = document.createElement('div'), text = document.createElement('span');
        div.className = 'alert info';
        text.textContent = 'Tracker connected: 16 bird(s) on sim://flockcal?birds=16&motion=exercise&rate=144&baud=921600: '
                           + 'position_matrix, group mode, 144.0 Hz, stream mode';
        const close = document.createElement('button'); close.className = 'close'; close.textContent = '×';
        div.append(text, close); box.prepend(div);
        return box.scrollWidth - box.clientWidth; })()""")
    page.screenshot(path=str(artifacts() / "fresh-dashboard-alert.png"), clip=page.locator("#session-panel").bounding_box())
    assert overflow <= 1, f"the Alerts box scrolls sideways by {overflow} px"
    assert not page.problems, page.problems
    page.close()

    kiosk = open_offline(browser, fresh_serve.url + "/kiosk", width=1280, height=800)
    kiosk.wait_for_function("!document.body.innerText.includes('Reconnecting')", timeout=20000)
    # "Fresh" is an operator's session (the fixture's): the kiosk shows no one and waits for the stage,
    # trying nothing that fails (docs/dashboard.md). The dashboard above drew the rig with the GLTFLoader.
    kiosk.wait_for_selector("#kiosk-state[data-state=busy]", timeout=20000)
    kiosk.wait_for_timeout(2500)
    kiosk.screenshot(path=str(artifacts() / "fresh-kiosk.png"))
    assert any(u.endswith("kiosk.js") for u, _ in kiosk.scripts)
    assert kiosk.scripts and all(status == 200 for _, status in kiosk.scripts), kiosk.scripts
    assert not kiosk.problems, kiosk.problems
    assert "in use" in kiosk.inner_text("#kiosk-state") and "Fresh" not in kiosk.inner_text("body")
    kiosk.close()


@pytest.mark.browser
@pytest.mark.parametrize("path, selector, text", [("/docs", ".swagger-ui .info .title", "flockcal"),
                                                  ("/redoc", "h1", "flockcal")])
def test_api_docs_render_offline_in_chromium(fresh_serve, browser, path, selector, text):
    page = open_offline(browser, fresh_serve.url + path)
    page.wait_for_selector(selector, timeout=20000)
    assert text in page.inner_text(selector)
    page.wait_for_timeout(500)
    page.screenshot(path=str(artifacts() / f"fresh{path.replace('/', '-')}.png"))
    # ReDoc's bundle asks for its makers' logo from their CDN; the page's Content-Security-Policy makes
    # the browser refuse it before any request leaves (so it is not in problems as a request), and
    # chromium says so on the console. Nothing else may go wrong.
    refused = [p for p in page.problems if "cdn.redoc.ly" in p and ("Content Security Policy" in p or p.endswith("(csp)"))]
    assert not [p for p in page.problems if p.startswith("external request")], page.problems
    assert not [p for p in page.problems if p not in refused], page.problems
    page.close()


def test_stopping_serve_says_what_it_saved(fresh_serve):
    # Runs last in this module: Ctrl-C the service the tests above used (a session is live).
    fresh_serve.send_signal(signal.SIGINT)
    # uvicorn re-raises the Ctrl-C once it has shut down (recent versions), so the command exits 130.
    assert fresh_serve.wait(30) in (0, 130)
    out = fresh_serve.log.read_text()
    assert re.search(r"flockcal serve: stopped session \S+ \(Fresh, \d+ frames\): result stored", out), out[-2000:]
    saved = re.findall(r"flockcal serve: saved (\S+)", out)
    assert saved and all(Path(p).exists() for p in saved), saved
    assert any(p.endswith(".frames") for p in saved)
