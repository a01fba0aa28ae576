"""Shared fixtures: the simulated performer on a fake Flock of Birds behind a real pty.

Module-scoped, so each test module gets its own performer and tracker; a module that needs another
routine or rate defines its own `performer`/`tracker` fixtures, which take precedence.
"""

import pytest

from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker

RATE_HZ = 144.0


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
