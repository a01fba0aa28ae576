"""Slip and swap detection (docs/slippage.md): `SlipMonitor` and `detect_slips` (monitor), the one slip loop
`SlipWatch` (watch), and the monitor's parts: step test (stats), baseline and confirming test (baseline),
recent frames (buffer), suspicions by onset (pending), attribution, and the same pose again (revisit).
"""

from flockcal.solver.slippage.monitor import SlipEvent, SlipMonitor, SlippageError, SwapEvent, detect_slips
from flockcal.solver.slippage.watch import SlipWatch

__all__ = ["SlipEvent", "SlipMonitor", "SlippageError", "SwapEvent", "SlipWatch", "detect_slips"]
