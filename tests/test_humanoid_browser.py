"""The pages say which limb each sensor was found on (issue 47), in a real headless chromium against a real
service on loopback reading the built-in sim:// performer whose two hand sensors were named the wrong way
round: the dashboard's topology shows the limb found for every sensor and alerts the two names that say
otherwise, once each; the kiosk names its chips by the limb found, and shows the attendant's strip (the
map and the two warnings) only with ?operator=1, never to a guest.
"""

from __future__ import annotations

import httpx
import pytest

from browser_helpers import NEEDS_CHROMIUM
from flockcal.server.settings import Settings
from humanoid_cases import swapped_hands
from server_helpers import ServerThread, free_port, wait_connected

pytestmark = [pytest.mark.browser, NEEDS_CHROMIUM]

ADMIN, READ = "admin-secret-47", "read-secret-47"
# The operator typed the names in cable order with the two hands swapped.
NAMES, TRUE = swapped_hands()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = Settings(device="sim://h47pages?birds=16&motion=walk&rate=60&baud=921600", birds=16, baud=921600,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("pages"), names=NAMES,
                        token=ADMIN, read_token=READ)
    with ServerThread(settings) as srv:
        wait_connected(srv.url, token=ADMIN)
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Ann"},
                       headers={"Authorization": f"Bearer {ADMIN}"}, timeout=30)
        assert r.status_code == 201, r.text
        yield srv


def open_page(browser, url: str):
    page = browser.new_page(viewport={"width": 1440, "height": 1000})
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    page.goto(url)
    return page


FOUND_JS = "() => Object.fromEntries([...document.querySelectorAll('#topology .found')].map(e => [e.dataset.sensor, e.dataset.bone]))"


def test_the_dashboard_shows_the_limb_found_for_every_sensor_and_alerts_each_name_that_disagrees(server, browser):
    page = open_page(browser, f"{server.url}/?token={ADMIN}")
    try:
        page.wait_for_function(f"({FOUND_JS})()['r_hand'] === 'leftHand' && "
                               "document.querySelectorAll('#topology .found').length === 16", timeout=60000)
        assert page.evaluate(FOUND_JS) == TRUE
        conflicted = page.eval_on_selector_all("#topology .found.conflict", "els => els.map(e => e.dataset.sensor)")
        assert sorted(conflicted) == ["l_hand", "r_hand"]
        page.wait_for_function("document.querySelectorAll('#alerts .alert.conflict').length === 2", timeout=10000)
        alerts = page.eval_on_selector_all("#alerts .alert.conflict span", "els => els.map(e => e.textContent)")
        assert any("'l_hand' is named for the left hand but was found on the right hand" in a for a in alerts)
        page.wait_for_timeout(1500)  # more fits arrive (15 a second): the warnings are not repeated
        assert len(page.query_selector_all("#alerts .alert.conflict")) == 2
        assert page.get_attribute("#topology-note", "data-humanoid") == "found"
        assert not page.errors, page.errors
    finally:
        page.close()


def test_the_kiosk_shows_the_map_and_warnings_to_the_attendant_only(server, browser):
    attendant = open_page(browser, f"{server.url}/kiosk?token={READ}&operator=1")
    guest = open_page(browser, f"{server.url}/kiosk?token={READ}")
    try:
        attendant.wait_for_function("document.querySelectorAll('#operator .found').length === 16 && "
                                    "document.querySelector('#operator .found[data-sensor=r_hand]').dataset.bone === 'leftHand'",
                                    timeout=60000)
        shown = attendant.eval_on_selector_all("#operator .found", "els => Object.fromEntries(els.map(e => [e.dataset.sensor, e.dataset.bone]))")
        assert shown == TRUE
        warnings = attendant.eval_on_selector_all("#operator .conflict", "els => els.map(e => e.textContent)")
        assert len(warnings) == 2 and all("check the strap or the name" in w for w in warnings)
        # The guest's screen: the avatar, chips named by the limb found; no strip, no warnings.
        guest.wait_for_function("document.querySelector('#chips .chip[data-body=r_hand]') !== null", timeout=60000)
        assert "left hand" in guest.text_content("#chips .chip[data-body=r_hand]")
        assert "hidden" in (guest.get_attribute("#operator", "class") or "")
        assert guest.query_selector_all("#operator .conflict") == []
        assert not attendant.errors and not guest.errors, attendant.errors + guest.errors
    finally:
        attendant.close()
        guest.close()
