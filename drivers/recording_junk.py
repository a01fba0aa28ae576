"""The junk of a `.fobraw` recording: chunks whose checksums hold but that no recorder wrote, counted by
`Decoder` (drivers/recording.py) as it skips them, with where they are and why each was judged so.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Junk:
    """Chunks whose checksums hold but that no recorder wrote (random or foreign data spliced in), all
    skipped: where they are and why each was judged so (a time out of the recording's order, a port it does
    not have, a marker that is not a recorder's JSON, read bytes with more phasing bits than Flock records
    can hold)."""

    chunks: int = 0
    bytes: int = 0
    first: int | None = None  # byte offset of the first such chunk
    end: int | None = None  # where the last one ends
    reasons: dict = field(default_factory=dict)  # reason → chunks

    def add(self, pos: int | None, end: int | None, size: int, reason: str) -> None:
        self.chunks += 1
        self.bytes += size
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        if pos is not None:
            self.first = pos if self.first is None else min(self.first, pos)
            self.end = end if self.end is None else max(self.end, end)

    def __bool__(self) -> bool:
        return self.chunks > 0

    def describe(self) -> str:
        where = f" between bytes {self.first:,} and {self.end:,}" if self.first is not None else ""
        why = "; ".join(f"{n:,} {reason}" for reason, n in sorted(self.reasons.items(), key=lambda x: -x[1]))
        return f"{self.chunks:,} junk chunk{'s' if self.chunks != 1 else ''} ({self.bytes:,} bytes){where}: {why}"
