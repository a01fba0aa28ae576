"""A simulated performer wearing tracker sensors, and a fake Flock of Birds on a pty or sim:// URL.

Importing this package registers the sim:// scheme with pyserial.
"""

import serial as _serial

# pyserial imports `<package>.protocol_<scheme>` for a `<scheme>://` URL from each package listed here.
if "flockcal.simulator" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("flockcal.simulator")
