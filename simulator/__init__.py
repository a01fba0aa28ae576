"""A simulated performer wearing tracker sensors, and a fake Flock of Birds on a pty or sim:// URL.

Importing this package registers the sim:// scheme with pyserial.
"""

import serial as _serial

# pyserial imports `<package>.protocol_<scheme>` for a `<scheme>://` URL from each package listed here.
if "flockcal.simulator" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("flockcal.simulator")

from flockcal.lazy import public_api  # noqa: E402 (after the scheme is registered, as importing promises)

# What a user of the simulator reaches for, each loaded on first use (tests/test_public_api.py resolves them).
__getattr__, __dir__, __all__ = public_api(__name__, {
    "simulate": "flockcal.simulator.take",
    "simulate_markers": "flockcal.simulator.optical",
    "Performer": "flockcal.simulator.performer",
    "BodyModel": "flockcal.simulator.body",
    "human": "flockcal.simulator.body",
    "linkage": "flockcal.simulator.body",
    "rigid_pair": "flockcal.simulator.body",
    "Motion": "flockcal.simulator.motion",
    "routine": "flockcal.simulator.motion",
    "FakeFlock": "flockcal.simulator.fake_tracker",
    "PtyTracker": "flockcal.simulator.pty_tracker",
    "ManualClock": "flockcal.clock",
    "SimulatorError": "flockcal.simulator.body",
})
