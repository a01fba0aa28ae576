"""Slip and swap detection (docs/slippage.md): `SlipMonitor` and `detect_slips` (monitor), its `SlipSettings`
(settings) and events (events), the one slip loop `SlipWatch` (watch), and the monitor's parts: the step test
(steptest, stats, baseline), the confirming test (confirming, attribution, revisit), the frame-rate step test
(framescan, framestep), recent frames (buffer) and suspicions by onset (pending).
"""

from flockcal.solver.slippage.events import SlipEvent, SlippageError, SwapEvent
from flockcal.solver.slippage.monitor import SlipMonitor, detect_slips
from flockcal.solver.slippage.settings import SlipSettings

__all__ = ["SlipEvent", "SlipMonitor", "SlipSettings", "SlippageError", "SwapEvent", "SlipWatch", "detect_slips"]


def __getattr__(name: str):
    # SlipWatch (the live loop) on first use: `flockcal fit` needs only `detect_slips`, and the watch pulls
    # in the segmented accumulator with it.
    if name == "SlipWatch":
        from flockcal.solver.slippage.watch import SlipWatch

        return SlipWatch
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
