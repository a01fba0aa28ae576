"""Is the stream as fast as the flock was set to? The measured frame rate against the asked one, and a
warning that names the cause (the line's speed for the record format, or the flock) and the fixes.
"""

from __future__ import annotations

from flockcal.drivers.link import BAUD_RATES, LINK_MARGIN, FlockSetup, link_capacity
from flockcal.drivers.records import record_length


class RateCheck:
    """Frames per second actually streamed, measured once over a window early in each session, against
    the measurement rate the flock was set to; the warning names the cause (the line's speed for the
    record format) and the fixes."""

    SETTLE_S = 0.5  # the stream's first records are skipped: the setup's drain and first cycles
    WINDOW_S = 2.0
    SHORTFALL = 0.9  # below 90 % of the asked rate is worth telling the operator

    def __init__(self, setup: FlockSetup, start: float):
        self.setup = setup
        self.start = start
        self.bytes = 0
        self.mark: tuple[float, int, int] | None = None  # (time, frames, bytes) at the window's start
        self.measured_hz: float | None = None
        self.done = False

    def check(self, now: float, frames: int) -> str | None:
        if self.done or now - self.start < self.SETTLE_S:
            return None
        if self.mark is None:
            self.mark = (now, frames, self.bytes)
            return None
        t0, f0, b0 = self.mark
        if now - t0 < self.WINDOW_S:
            return None
        self.done = True
        self.measured_hz = (frames - f0) / (now - t0)
        return rate_warning(self.setup, self.measured_hz, (self.bytes - b0) / (now - t0))


def rate_warning(setup: FlockSetup, measured_hz: float, bytes_per_s: float | None = None) -> str | None:
    """None when `measured_hz` is near the flock's rate, else one line: what was asked, what came, why
    (the line's speed for the record format, or the flock itself), and the fixes."""
    asked = setup.rate_hz
    if not asked or measured_hz >= RateCheck.SHORTFALL * asked:
        return None
    on_port = setup.birds if setup.group else 1
    per_set = lambda fmt: on_port * record_length(fmt, group=setup.group)  # noqa: E731
    need = per_set(setup.record_format) * asked
    claimed = link_capacity(setup.baud)
    got = bytes_per_s if bytes_per_s is not None else per_set(setup.record_format) * measured_hz
    text = (f"{measured_hz:.1f} frames/s arrive but the flock measures at {asked:g} Hz: {setup.record_format} for "
            f"{on_port} bird(s) on one line needs {need:.0f} B/s")
    fixes = []
    if need > claimed * LINK_MARGIN:
        text += f", more than {setup.baud} baud carries ({claimed:.0f} B/s)"
        capacity = claimed
    elif got < 0.8 * claimed:
        # The line should carry it but brings far less: the unit's DIP switches set a slower speed than --baud.
        real = next((b for b in BAUD_RATES if link_capacity(b) >= got), BAUD_RATES[-1])
        text += (f", which {setup.baud} baud would carry, but the line delivers only {got:.0f} B/s: it runs "
                 f"slower than --baud says (at most {real} baud)")
        fixes.append("--baud matching the unit's DIP switches (RS-232 tops out at 115200), so the driver picks a "
                     "record format that fits")
        capacity = link_capacity(real)
    else:
        return text + ("; the line carries that, so the flock itself falls behind — look for bird errors "
                       "(error 31: lower --rate)")
    budget = capacity * LINK_MARGIN
    compact = [f for f in ("position_quaternion", "position_angles")
               if per_set(f) < per_set(setup.record_format) and per_set(f) * asked <= budget]
    if compact:
        fixes.append(f"--format {compact[0]}")
    fixes.append(f"--rate {max(1, int(budget // per_set(setup.record_format)))} or lower")
    if setup.group and setup.birds > 1:
        fixes.append("one port per bird (--per-port)")
    return f"{text} — use {', or '.join(fixes)}"
