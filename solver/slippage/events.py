"""What the slippage monitor reports: a `SlipEvent` (a sensor moved on the body) or a `SwapEvent` (two sensors
exchanged streams), and `SlippageError` for inputs it cannot use.
"""

from __future__ import annotations

from dataclasses import dataclass

from flockcal.errors import FlockcalError


class SlippageError(FlockcalError, ValueError):
    """Inputs the slippage monitor cannot use (shapes, names, a calibration without joints)."""


@dataclass(frozen=True)
class SlipEvent:
    """One sensor moved on the body: when, which (with the alternatives), which joints, how far."""

    time_s: float  # estimated time of the slip (first frame of the step)
    sensor: str
    candidates: tuple[str, ...]  # sensors that could explain it, most likely first
    confidence: float  # posterior share of `sensor`
    joints: tuple[str, ...]  # the affected joints, each named by its child body
    jump_mm: float  # size of the residual step
    detected_s: float = float("nan")  # time of the frame at which the monitor reported it
    sensor_index: int = -1
    joint_indices: tuple[int, ...] = ()

    kind = "slip"

    def to_dict(self) -> dict:
        """The `slip_events` entry of docs/design.md §5 (extended with kind, confidence and detected_s)."""
        return {"kind": "slip", "time_s": round(self.time_s, 4), "sensor": self.sensor,
                "candidates": list(self.candidates), "confidence": round(self.confidence, 4),
                "joints": list(self.joints), "jump_mm": round(self.jump_mm, 2),
                "detected_s": round(self.detected_s, 4)}


@dataclass(frozen=True)
class SwapEvent:
    """Two sensors exchanged identity (their data streams swapped) from `time_s` on."""

    time_s: float
    a: str
    b: str
    joints: tuple[str, ...]
    jump_mm: float
    confidence: float = 1.0
    detected_s: float = float("nan")
    sensor_indices: tuple[int, int] = (-1, -1)
    joint_indices: tuple[int, ...] = ()

    kind = "swap"

    @property
    def sensor(self) -> str:
        return self.a

    @property
    def candidates(self) -> tuple[str, ...]:
        return (self.a, self.b)

    def to_dict(self) -> dict:
        """A `slip_events` entry of kind "swap": `sensor` and `candidates` name both sensors."""
        return {"kind": "swap", "time_s": round(self.time_s, 4), "sensor": self.a,
                "candidates": [self.a, self.b], "sensors": [self.a, self.b],
                "confidence": round(self.confidence, 4), "joints": list(self.joints),
                "jump_mm": round(self.jump_mm, 2), "detected_s": round(self.detected_s, 4)}
