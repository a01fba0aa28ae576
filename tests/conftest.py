"""Shared fixtures: the simulated performer on a fake Flock of Birds behind a real pty.

Module-scoped, so each test module gets its own performer and tracker; a module that needs another
routine or rate defines its own `performer`/`tracker` fixtures, which take precedence.
"""

import os

import pytest
from hypothesis import HealthCheck, settings

from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker

RATE_HZ = 144.0

# Property tests: CI runs the same fixed examples every time (derandomized, nothing written to a
# .hypothesis database), so a red run is reproducible and a green one is not luck. Exploration with many
# fresh examples is `python benchmarks/hypothesis_explore.py` (the "explore" profile), never in CI.
_SLOW = [HealthCheck.too_slow, HealthCheck.data_too_large]
settings.register_profile("ci", max_examples=15, derandomize=True, database=None, deadline=None,
                          suppress_health_check=_SLOW, print_blob=True)  # fmt: skip
settings.register_profile("explore", max_examples=int(os.environ.get("FLOCKCAL_EXAMPLES", "400")),
                          deadline=None, suppress_health_check=_SLOW, print_blob=True)  # fmt: skip
settings.load_profile(os.environ.get("FLOCKCAL_HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(scope="module")
def performer():
    # The exercise routine compressed to an 8 s loop moves every joint within a few seconds.
    return Performer("human", "exercise", seed=1, rate_hz=RATE_HZ, period=8.0)


@pytest.fixture(scope="module")
def tracker(performer):
    # 16 birds at 144 Hz need a faster line than 115200 baud: emulate 921600 on the pty.
    pty = PtyTracker(performer, birds=16, baud=921600, rate_hz=RATE_HZ).start()
    yield pty
    pty.stop()


@pytest.fixture(scope="module")
def browser():
    """One headless chromium per module (tests/browser_helpers.py), for the page tests."""
    from playwright.sync_api import sync_playwright

    from browser_helpers import launch

    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()
