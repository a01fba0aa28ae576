"""What every accumulator the solver fits from offers: `GramAccumulator` and `SegmentedAccumulator`.

The server and `solve` hold an `Accumulator` and never ask which kind it is: a plain one is its own
whole take with no segments; a segmented one also answers per-pair fits on the frames since a slip.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable


@runtime_checkable
class Accumulator(Protocol):
    """Frame sums a calibration is read from (docs/internals.md, "The accumulator protocol")."""

    n_sensors: int

    @property
    def frames(self) -> int:
        """Frames fed so far."""
        ...

    def ingest(self, times, rotations, positions, valid=None) -> "Accumulator":
        """Add frames (times in seconds, (n, m, 3, 3) rotations, (n, m, 3) positions, (n, m) valid)."""
        ...

    def copy(self) -> "Accumulator":
        """An independent copy a fit on another thread can read while this one keeps growing."""
        ...

    @property
    def whole_take(self):
        """The `GramAccumulator` of every frame fed."""
        ...

    @property
    def segments(self) -> Mapping:
        """{sensor index: Segment} open after slips; empty for a plain accumulator."""
        ...

    def pair_view(self):
        """A `GramAccumulator`-like object whose pair statistics come from each pair's segment."""
        ...
