"""Slip and swap detection (docs/slippage.md): `SlipMonitor` and `detect_slips` (monitor), the one slip loop
`SlipWatch` (watch), and the monitor's parts: step test (stats), baseline and confirming test (baseline),
recent frames (buffer), suspicions by onset (pending), attribution, and the same pose again (revisit).
"""

from flockcal.solver.slippage.monitor import SlipEvent, SlipMonitor, SlippageError, SwapEvent, detect_slips

__all__ = ["SlipEvent", "SlipMonitor", "SlippageError", "SwapEvent", "SlipWatch", "detect_slips"]


def __getattr__(name: str):
    # SlipWatch (the live loop) on first use: `flockcal fit` needs only `detect_slips`, and the watch pulls
    # in the segmented accumulator with it.
    if name == "SlipWatch":
        from flockcal.solver.slippage.watch import SlipWatch

        return SlipWatch
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
