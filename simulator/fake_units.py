"""The fake flock's state: one unit on the FBB (`Bird`), one RS-232 line (`Line`), and the
constants a real bird reports (software revision, crystal, default and largest measurement rate).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flockcal.drivers.records import DEFAULT_FORMAT, RecordFormat

SOFTWARE_REVISION = 3.67
CRYSTAL_MHZ = 25
DEFAULT_RATE_HZ = 103.0  # p7 default 0x6700
MAX_RATE_HZ = 180.0  # the bird cannot measure faster [MAN p146]
OUTPUT_BUFFER_LIMIT = 65536  # bytes delivered but not read before the oldest are lost (host overrun)


@dataclass
class Bird:
    """Per-address state (one unit on the FBB)."""

    address: int
    sensor_index: int | None  # index into the pose source; None for an ERC/ERT unit
    fmt: RecordFormat = DEFAULT_FORMAT
    hemisphere: str = "forward"
    hemisphere_via_p22: bool = False
    button_mode: bool = False
    metal: bool = False
    running: bool = False
    scale_p3: int = 0  # position scaling (p3 byte 0): 0 = 36 in, 1 = 72 in; each bird keeps its own
    params: dict[int, bytes] = field(default_factory=dict)


@dataclass
class Line:
    """One RS-232 port: the parser of host bytes and the bird→host byte queue with delivery times."""

    index: int
    home: int  # address a command without an RS232-TO-FBB prefix goes to
    baud: float
    data: bytearray = field(default_factory=bytearray)
    done: np.ndarray = field(default_factory=lambda: np.zeros(0))  # delivery time of each byte
    free_at: float = 0.0  # when the transmitter of this line is idle again
    connected: bool = True
    stream: bool = False
    stream_address: int | None = None  # non-group STREAM target
    xoff: bool = False
    stalled_until: float = -np.inf
    drop_pending: int = 0
    # parser
    pending: bytearray = field(default_factory=bytearray)
    prefix: int | None = None
    super_prefix: bool = False
    # counters
    records_sent: int = 0
    sets_skipped: int = 0
    bytes_lost: int = 0
    bytes_received: int = 0

    @property
    def bytes_per_second(self) -> float:
        return self.baud / 10.0
